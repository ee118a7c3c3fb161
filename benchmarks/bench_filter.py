"""Benchmark: one vehicle-step of the MM-PHD-SLAM filter on the analytic ``paper`` data.

Runs the cooperative filter loop (both vehicles, map fusion at the BS: the stages of
:class:`mmslam.slam.filter.run.CooperativeRun`, as ``run_filter``, without the evaluation) and
times every :meth:`LocalFilter.step` call (predict + correct + reduce + estimate + resample) of
vehicle 1 from step ``--warmup`` on, on one core (OMP / OpenBLAS / MKL threads set to 1 before
NumPy is imported). Reports the median and quartiles per variant and particle count.

    python benchmarks/bench_filter.py                  # baseline + proposed at P = 300, all 40 steps
    python benchmarks/bench_filter.py --scaling        # also P = 100, 300, 1000, 3000 (first 20 steps)
    python benchmarks/bench_filter.py --cpu            # thread CPU time (busy machine)
    python benchmarks/bench_filter.py --set filter.types.VA.tail_weight=0.2   # paper data, a setting changed
    python benchmarks/bench_filter.py --city           # the built-in VA row (a city scene's defaults) on the paper data

docs/design.md section 8 targets: <= 10 ms median for ``proposed`` at P = 300; cost linear in P.

The filter's kernels are compiled by numba on first use and cached on disk (``cache=True``), so
vehicle 1's first step (which runs every kernel) is reported on its own: the compile time on a
cold cache (``NUMBA_CACHE_DIR=$(mktemp -d) python benchmarks/bench_filter.py``), else the time to
load the cached machine code. It is not part of the per-step statistics.
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from mmslam.raytrace.analytic import AnalyticSource  # noqa: E402
from mmslam.errors import MmslamError  # noqa: E402
from mmslam.scenes.scenario import DEFAULT_TYPE_PARAMS, load_preset, with_overrides  # noqa: E402
from mmslam.scenes.trajectory import vehicle_trajectories  # noqa: E402
from mmslam.slam.filter.run import CooperativeRun  # noqa: E402


def paper_data(steps: int):
    scn = load_preset("paper")
    states = vehicle_trajectories(scn, steps)
    src = AnalyticSource(scn)
    parts = [src.trace_step(k, states[k]) for k in range(steps)]
    paths = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    return scn, states, paths


def city_va_row() -> list[str]:
    """``--set`` strings that give the paper data the built-in VA row (``DEFAULT_TYPE_PARAMS["VA"]``: what a scene
    without a ``[filter.types.VA]`` table gets, the city defaults) in place of the ``paper`` preset's pinned one."""
    row = DEFAULT_TYPE_PARAMS["VA"]
    out = []
    for f in dataclasses.fields(row):
        v = getattr(row, f.name)
        if v is None:
            continue
        text = json.dumps(list(v) if isinstance(v, tuple) else v)  # TOML values: strings, numbers, booleans, arrays
        out.append(f"filter.types.VA.{f.name}={text}")
    return out


def time_steps(scn, states, paths, variant: str, particles: int, steps: int, warmup: int,
               seed: int = 0, clock=time.perf_counter) -> tuple[np.ndarray, float]:
    """Times (s) of vehicle 1's local steps ``warmup..steps-1`` in a full cooperative run, and the
    time (s) of its first step (numba compile or cache load on first use in the process).

    ``clock``: ``time.perf_counter`` (wall time) or ``time.thread_time`` (CPU time of this
    thread: less sensitive to other processes on a busy machine).
    """
    run = CooperativeRun(scn, states, paths, variant, particles, seed, steps, evaluate=False)
    times = []
    for k in range(steps):
        run.predict_at_bs(k)
        for n in range(run.n_veh):
            Z, spd, tr, R_z = run.local_inputs(k, n)
            t0 = clock()
            est = run.filters[n].step(Z, spd, tr, R_z)
            dt = clock() - t0
            if n == 0 and k >= warmup:
                times.append(dt)
            if n == 0 and k == 0:
                first = dt
            run.upload(k, n, est)
    return np.array(times), first


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=300)
    ap.add_argument("--variants", default="baseline,proposed")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--scaling", action="store_true", help="also time P = 100, 300, 1000, 3000")
    ap.add_argument("--scaling-steps", type=int, default=20)
    ap.add_argument("--cpu", action="store_true", help="time with the thread CPU clock instead of wall time")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a scenario parameter of the paper data (as mmslam slam --set), e.g. "
                         "filter.types.VA.tail_weight=0.2 to time the city VA row's heavy tail")
    ap.add_argument("--city", action="store_true",
                    help="time the built-in VA row (the defaults of a scene without a [filter.types.VA] table: the "
                         "city defaults) instead of the paper preset's pinned one; --set applies on top")
    args = ap.parse_args()
    clock = time.thread_time if args.cpu else time.perf_counter

    scn, states, paths = paper_data(max(args.steps, args.scaling_steps))
    try:
        scn = with_overrides(scn, (city_va_row() if args.city else []) + args.set)
    except MmslamError as e:
        ap.error(str(e))
    print(f"one vehicle-step (vehicle 1), analytic paper data{' with the built-in VA row' if args.city else ''}"
          f"{', --set ' + ' '.join(args.set) if args.set else ''}, "
          f"1 thread, {'CPU' if args.cpu else 'wall'} time; steps {args.warmup}..{args.steps - 1}")
    for v in args.variants.split(","):
        t, first = time_steps(scn, states, paths, v, args.particles, args.steps, args.warmup, clock=clock)
        q1, med, q3 = np.percentile(t * 1e3, [25, 50, 75])
        print(f"  {v:9s} P={args.particles:5d}: median {med:7.1f} ms  (IQR {q1:.1f}-{q3:.1f}, n={t.size}); "
              f"first step {first:.2f} s (numba compile / cache load)")
    if args.scaling:
        print(f"scaling (steps {args.warmup}..{args.scaling_steps - 1}):")
        for v in args.variants.split(","):
            base = None
            for P in (100, 300, 1000, 3000):
                t, _ = time_steps(scn, states, paths, v, P, args.scaling_steps, args.warmup, clock=clock)
                med = float(np.median(t)) * 1e3
                base = base or med / P
                print(f"  {v:9s} P={P:5d}: median {med:8.1f} ms   ms/particle {med / P:.4f}  "
                      f"(x{med / (base * P):.2f} of linear from P=100)")


if __name__ == "__main__":
    main()
