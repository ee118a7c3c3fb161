"""Benchmark: Sionna RT per-step trace of the `paper` preset on the CPU (LLVM backend).

Run: ``python benchmarks/bench_trace.py [--steps 40] [--samples 1000000] [--max-depth 1]``.
Scene build, load and one warm-up step (kernel tracing/compilation) are timed separately and
excluded from the per-step numbers. Prints median / max per step, the total for all steps, and
how many labelled rows per type were produced. DESIGN.md target: 40 steps <= 60 s on 2 cores.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--steps", type=int, default=None, help="steps to trace (default: the scenario's)")
    ap.add_argument("--samples", type=int, default=10**6, help="samples_per_src")
    ap.add_argument("--max-depth", type=int, default=1)
    args = ap.parse_args()

    from mmslam.scenes.scenario import resolve_scenario
    from mmslam.scenes.trajectory import vehicle_trajectories

    scn = resolve_scenario(args.scenario)
    steps = args.steps or scn.steps
    states = vehicle_trajectories(scn, steps)

    t0 = time.perf_counter()
    from mmslam.raytrace.sionna_adapter import SionnaSource

    src = SionnaSource(scn, max_depth=args.max_depth, samples_per_src=args.samples, seed=0)
    t_init = time.perf_counter() - t0
    t0 = time.perf_counter()
    src.trace_step(0, states[0])  # warm-up: traces and compiles the kernels
    t_warm = time.perf_counter() - t0

    import drjit as dr

    per_step = []
    counts = np.zeros(5, int)
    kernels = misses = backend_ms = 0
    t_all = time.perf_counter()
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history_clear()
        for k in range(steps):
            t0 = time.perf_counter()
            out = src.trace_step(k, states[k])
            per_step.append(time.perf_counter() - t0)
            counts += np.bincount(out["type"].astype(int), minlength=5)
            for h in dr.kernel_history([dr.KernelType.JIT]):
                kernels += 1
                misses += not h.get("cache_hit", True)
                backend_ms += h.get("backend_time", 0.0)
    total = time.perf_counter() - t_all

    v = src.versions()
    print(f"scenario {scn.name}: {steps} steps, {len(scn.vehicles)} receivers, max_depth {args.max_depth}, "
          f"samples_per_src {args.samples}, {v['variant']} (sionna-rt {v['sionna-rt']}, drjit {v['drjit']})")
    print(f"scene build + load: {t_init:.2f} s; warm-up step (kernel compile): {t_warm:.2f} s")
    print(f"per step: median {statistics.median(per_step) * 1e3:.0f} ms, max {max(per_step) * 1e3:.0f} ms")
    print(f"total {steps} steps: {total:.2f} s (target <= 60 s)")
    print(f"JIT kernels launched after warm-up: {kernels}; not in the in-memory cache (re-traced): {misses}; "
          f"backend compile time {backend_ms / 1e3:.2f} s")
    print("rows per type: " + ", ".join(f"{n}={c}" for n, c in zip(("BS", "VA", "SP", "VS", "OTHER"), counts)))


if __name__ == "__main__":
    main()
