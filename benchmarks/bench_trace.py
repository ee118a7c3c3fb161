"""Benchmark: Sionna RT per-step trace of the shipped scenes (CPU/LLVM, or CUDA when present).

Run: ``python benchmarks/bench_trace.py [--scenario paper,street,canyon,munich] [--steps 10]
[--samples 1000000] [--max-depth 1] [--cpu]``.

Per scenario: scene build + load, one warm-up step (step 0: kernel tracing / compilation) timed
separately and excluded; then ``--steps`` steps spread over the trajectory (step 0 again
included) timed one by one. Prints median / max per step, the JIT kernels launched after the
warm-up and how many were not in the in-memory kernel cache (re-traced: should be 0), and the
labelled rows per type. Targets (docs/design.md section 8): ``paper`` 40 steps <= 10 s on 2 CPU cores;
``munich`` (5 cars, depth 1, 1e6 rays) <= 0.5 s per step. ``--cpu`` forces the LLVM backend
(``MMSLAM_FORCE_CPU=1``); otherwise a working CUDA device is used. Timings on a shared machine
are noisy: the load average is printed with each result.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

CASES = ("paper", "street", "canyon", "munich")


def bench_one(name: str, steps: int, samples: int, max_depth: int) -> dict:
    """Trace ``steps`` steps of preset ``name``; per-step seconds and kernel statistics."""
    import drjit as dr

    from mmslam.raytrace.sionna_adapter import SionnaSource
    from mmslam.scenes.scenario import resolve_scenario
    from mmslam.scenes.trajectory import vehicle_trajectories

    scn = resolve_scenario(name)
    states = vehicle_trajectories(scn)
    ks = np.unique(np.linspace(0, scn.steps - 1, min(steps, scn.steps)).round().astype(int))
    t0 = time.perf_counter()
    src = SionnaSource(scn, max_depth=max_depth, samples_per_src=samples, seed=0)
    t_init = time.perf_counter() - t0
    t0 = time.perf_counter()
    src.trace_step(0, states[0])  # warm-up: traces and compiles the kernels
    t_warm = time.perf_counter() - t0
    per_step, counts = [], np.zeros(5, int)
    kernels = misses = 0
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history_clear()
        for k in ks:
            t0 = time.perf_counter()
            out = src.trace_step(int(k), states[k])
            per_step.append(time.perf_counter() - t0)
            counts += np.bincount(out["type"].astype(int), minlength=5)
            for h in dr.kernel_history([dr.KernelType.JIT]):
                kernels += 1
                misses += not h.get("cache_hit", True)
    return {"scenario": name, "objects": len(src.scene.objects), "vehicles": len(scn.vehicles),
            "steps": len(ks), "init_s": t_init, "warm_s": t_warm, "median_s": statistics.median(per_step),
            "max_s": max(per_step), "kernels": kernels, "misses": misses, "counts": counts,
            "versions": src.versions(), "load": os.getloadavg()[0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=",".join(CASES), help="comma-separated presets or .toml files")
    ap.add_argument("--steps", type=int, default=10, help="timed steps per scenario (spread over the trajectory)")
    ap.add_argument("--samples", type=int, default=10**6, help="samples_per_src")
    ap.add_argument("--max-depth", type=int, default=1)
    ap.add_argument("--cpu", action="store_true", help="force the LLVM (CPU) backend")
    ap.add_argument("--no-merge", action="store_true",
                    help="load external scenes unmerged (one object per XML shape), for an A/B comparison")
    args = ap.parse_args()
    if args.no_merge:
        from mmslam.backend import import_mitsuba

        import_mitsuba()
        import sionna.rt as rt

        load = rt.load_scene
        rt.load_scene = lambda *a, **k: load(*a, **{**k, "merge_shapes": False})
    if args.cpu:
        os.environ["MMSLAM_FORCE_CPU"] = "1"
    print(f"{'scenario':<10} {'objects':>7} {'cars':>4} {'steps':>5} {'load s':>7} {'warm s':>7} "
          f"{'median ms':>9} {'max ms':>7} {'kernels':>7} {'retraced':>8} {'loadavg':>7}  rows BS/VA/SP/VS/OTHER")
    for name in args.scenario.split(","):
        r = bench_one(name.strip(), args.steps, args.samples, args.max_depth)
        print(f"{r['scenario']:<10} {r['objects']:>7} {r['vehicles']:>4} {r['steps']:>5} {r['init_s']:>7.2f} "
              f"{r['warm_s']:>7.2f} {r['median_s'] * 1e3:>9.0f} {r['max_s'] * 1e3:>7.0f} {r['kernels']:>7} "
              f"{r['misses']:>8} {r['load']:>7.2f}  {'/'.join(map(str, r['counts']))}", flush=True)
    v = r["versions"]
    print(f"backend {v['variant']}, sionna-rt {v['sionna-rt']}, drjit {v['drjit']}, samples_per_src {args.samples}, "
          f"{'unmerged' if args.no_merge else 'merged'} external scenes, "
          f"max_depth {args.max_depth}; targets: munich median <= 500 ms, paper 40 steps <= 10 s (CPU)")


if __name__ == "__main__":
    main()
