"""Benchmark: analytic trace of a scenario into a fresh cache, and reloading caches.

Usage::

    python benchmarks/bench_cache.py [--scenario paper] [--steps N] [--repeats 5] [--cache DIR ...]
                                     [--json OUT.json]

Reports medians (and min / max) over ``--repeats`` runs of

- ``analytic_trace_s``: :func:`trace_scenario` with the analytic source into an empty temporary
  root (no progress bar): trajectories, closed-form paths, Parquet chunks, manifest;
- ``analytic_step_s``: one :meth:`AnalyticSource.trace_step` call (both receivers);
- ``load_s``: :func:`load_cache` of that cache (sha256 + Parquet read + validation);
- for each ``--cache DIR`` (e.g. a Sionna cache from ``mmslam trace paper --source sionna``):
  its reload time, and, when its manifest is a Sionna trace, the ratio against the Sionna
  trace time you pass with ``--sionna-trace-s`` (measured by ``benchmarks/bench_trace.py``).

Wall-clock seconds on this machine; single process.
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path


def _timeit(fn, repeats: int) -> dict:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return {"median": statistics.median(ts), "min": min(ts), "max": max(ts), "n": repeats}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="paper", help="preset name or .toml file")
    ap.add_argument("--steps", type=int, default=None, help="steps to trace (default: the scenario's)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--cache", action="append", default=[], help="also time reloading this cache dir")
    ap.add_argument("--sionna-trace-s", type=float, default=None,
                    help="Sionna trace time of the --cache trace (s), for the reload speed-up ratio")
    ap.add_argument("--json", type=Path, default=None, help="write the results here (a new file, or one an earlier "
                    "--json wrote: nothing else is replaced)")
    a = ap.parse_args(argv)
    if a.json is not None:  # before any timing: a user's file is refused, never replaced
        from mmslam.outputs import check_file_target

        check_file_target(a.json, "bench_cache", is_bench_cache_json, option="--json")

    from mmslam.raytrace.analytic import AnalyticSource
    from mmslam.raytrace.cache import load_cache
    from mmslam.raytrace.trace import trace_scenario
    from mmslam.scenes.scenario import resolve_scenario
    from mmslam.scenes.trajectory import vehicle_trajectories

    scn = resolve_scenario(a.scenario)
    steps = scn.steps if a.steps is None else a.steps
    res: dict = {"benchmark": "bench_cache", "scenario": scn.name, "steps": steps, "vehicles": len(scn.vehicles)}
    src = AnalyticSource(scn)
    states = vehicle_trajectories(scn, steps)

    with tempfile.TemporaryDirectory(prefix="bench_cache_") as tmp:
        counter = iter(range(10**6))

        def trace_fresh():
            return trace_scenario(scn, src, Path(tmp) / f"r{next(counter)}", steps=steps, progress=False)

        res["analytic_trace_s"] = _timeit(trace_fresh, a.repeats)
        res["analytic_step_s"] = _timeit(lambda: src.trace_step(steps // 2, states[steps // 2]), a.repeats * 20)
        d = trace_fresh()
        c = load_cache(d)
        res["paths_rows"] = int(len(c.paths["rx"]))
        res["chunks"] = len(c.manifest["chunks"])
        res["load_s"] = _timeit(lambda: load_cache(d), a.repeats)
    res["trace_over_load"] = res["analytic_trace_s"]["median"] / res["load_s"]["median"]

    res["caches"] = []
    for cd in a.cache:
        c = load_cache(cd)
        r = {"cache": str(c.path), "source": c.manifest["source"], "steps": c.steps,
             "paths_rows": int(len(c.paths["rx"])), "load_s": _timeit(lambda: load_cache(cd), a.repeats)}
        if a.sionna_trace_s is not None and c.manifest["source"] == "sionna":
            r["sionna_trace_s"] = a.sionna_trace_s
            r["trace_over_load"] = a.sionna_trace_s / r["load_s"]["median"]
        res["caches"].append(r)

    def fmt(t: dict) -> str:
        return f"{t['median'] * 1e3:9.2f} ms (min {t['min'] * 1e3:.2f}, max {t['max'] * 1e3:.2f}, n={t['n']})"

    print(f"scenario {res['scenario']}: {steps} steps x {res['vehicles']} receivers, "
          f"{res['paths_rows']} path rows in {res['chunks']} chunks")
    print(f"analytic trace (fresh cache) {fmt(res['analytic_trace_s'])}")
    print(f"analytic trace_step          {fmt(res['analytic_step_s'])}")
    print(f"load_cache                   {fmt(res['load_s'])}")
    print(f"trace / load                 {res['trace_over_load']:9.1f} x")
    for r in res["caches"]:
        line = f"load_cache {r['cache']} ({r['source']}, {r['steps']} steps, {r['paths_rows']} rows) {fmt(r['load_s'])}"
        if "trace_over_load" in r:
            line += f"; sionna trace / load = {r['trace_over_load']:.0f} x"
        print(line)
    if a.json is not None:
        from mmslam.outputs import atomic_write_bytes

        atomic_write_bytes(a.json, (json.dumps(res, indent=1) + "\n").encode(), fsync=False)
    return 0


def is_bench_cache_json(path: Path) -> bool:
    """True if ``path`` holds the JSON an earlier ``--json`` wrote (its ``"benchmark": "bench_cache"`` entry, or, from
    before that entry, its ``analytic_trace_s``, ``load_s`` and ``trace_over_load`` results)."""
    try:
        data = json.loads(Path(path).read_bytes())
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and (data.get("benchmark") == "bench_cache"
                                       or {"analytic_trace_s", "load_s", "trace_over_load"} <= set(data))


if __name__ == "__main__":
    from script_entry import run

    run(main, "bench_cache.py")
