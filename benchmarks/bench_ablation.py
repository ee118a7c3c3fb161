"""Benchmark: the full ablation from a cached analytic trace (docs/design.md section 8).

3 variants x 10 Monte Carlo runs x 40 steps x 2 vehicles at P = 300 on the ``paper`` preset,
local process pool over all cores. Target: <= 60 s on 2 cores.

The trace is made (or reused) first and is not timed; each repetition then runs the whole grid
in a fresh results directory (no job is reused), and the median wall time is printed.

    python benchmarks/bench_ablation.py [--mc 10] [--particles 300] [--steps 40] [--workers N]
                                        [--executor local|dask] [--repeat 1] [--keep DIR]
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from mmslam.pipelines.ablate import VARIANTS, prepare_cache, run_ablation

TARGET_S = 60.0


def _keep_names() -> tuple[str, ...]:
    """What an ablation folder holds (its marker aside): a kept folder holding anything else is refused, so a
    file the user added to it is never deleted."""
    from mmslam.pipelines.ablate.options import ABLATION_FILE, JOBS_DIR, SUMMARY_JSON, SUMMARY_PARQUET

    return (ABLATION_FILE, JOBS_DIR, SUMMARY_JSON, SUMMARY_PARQUET)


def check_keep(keep: Path) -> Path:
    """``--keep``: a new or empty folder, or one an earlier ``--keep`` wrote (its marker, nothing else in it); else
    a one-line :class:`~mmslam.errors.MmslamError`. Returns the folder to write (a link's target)."""
    from mmslam.outputs import check_target
    from mmslam.pipelines.ablate.store import ABLATION_KIND

    return check_target(keep, ABLATION_KIND, option="--keep", own_names=_keep_names())


def keep_ablation(out: Path, keep: Path) -> None:
    """Copy the finished ablation ``out`` to ``keep``, replacing an earlier kept one atomically (checked again:
    the folder may have changed during the run); the temporary copy is removed if anything fails."""
    from mmslam.outputs import make_temp_dir, replace_dir
    from mmslam.pipelines.ablate.store import ABLATION_KIND

    real = check_keep(keep)
    tmp = make_temp_dir(real.parent, real.name)
    try:
        shutil.copytree(out, tmp, dirs_exist_ok=True)
        replace_dir(tmp, real, ABLATION_KIND, own_names=_keep_names())
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mc", type=int, default=10)
    ap.add_argument("--particles", type=int, default=300)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--workers", type=int, default=None, help="default: all cores")
    ap.add_argument("--executor", default="local", choices=("local", "dask"))
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--keep", type=Path, default=None, help="keep the last repetition's ablation in this directory (new, "
                    "empty, or an ablation kept before: nothing else is replaced)")
    a = ap.parse_args(argv)
    if a.keep is not None:  # before any work: a user's folder is refused, not deleted
        check_keep(a.keep)

    root = Path(tempfile.mkdtemp(prefix="mmslam-bench-ablation-"))
    try:
        cache = prepare_cache("paper", "analytic", root / "trace", steps=a.steps, progress=False)
        times = []
        for i in range(a.repeat):
            out = root / f"run{i}"  # the ablation's own folder: nothing else in it (an ablation refuses a foreign one)
            shutil.copytree(root / "trace" / "cache", root / f"cache{i}")
            cache_i = root / f"cache{i}" / cache.name
            t0 = time.perf_counter()
            run = run_ablation(cache_i, out, VARIANTS, mc=a.mc, particles=a.particles, steps=a.steps,
                               executor=a.executor, workers=a.workers, progress=sys.stderr.isatty())
            dt = time.perf_counter() - t0
            assert len(run.ran) == len(VARIANTS) * a.mc, "every job must run in a fresh directory"
            times.append(dt)
            per_job = [r["wall_time_s"] for r in run.summary.headline if r["map"] == "fused"]
            print(f"run {i}: {dt:.1f} s wall for {len(run.ran)} jobs ({run.executor}); mean filter time per "
                  f"job by variant: " + ", ".join(f"{v} {t:.2f} s" for v, t in zip(VARIANTS, per_job)))
            if a.keep is not None and i == a.repeat - 1:
                keep_ablation(out, a.keep)
        med = statistics.median(times)
        print(f"bench_ablation: {len(VARIANTS)} variants x {a.mc} runs x {a.steps} steps x 2 vehicles, "
              f"P = {a.particles}, {os.cpu_count()} cores: median wall time {med:.1f} s "
              f"(target <= {TARGET_S:.0f} s: {'met' if med <= TARGET_S else 'NOT met'})")
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    from script_entry import run

    run(main, "bench_ablation.py")
