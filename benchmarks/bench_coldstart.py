"""Benchmark: cold start of a fresh install, the first ``mmslam slam`` on ``paper`` with no compiled kernels.

Traces the ``paper`` preset once with the analytic source (the filter's compile work does not depend
on the path source), then times whole ``mmslam slam`` processes (wall clock, and the CPU time of the
process and its children: the compile workers) on a new, empty ``NUMBA_CACHE_DIR`` each, followed by
the same command on the now warm cache. Also reports the run's own ``wall_time_s`` (stored in the
result, compile excluded) and the compile notice the first run printed. ``--serial`` compiles in
the run's own process (``--processes 1`` of :mod:`mmslam.slam.filter.precompile`), the behaviour before
parallel compilation, for comparison.

    python benchmarks/bench_coldstart.py                    # proposed, 2 cold + 1 warm runs
    python benchmarks/bench_coldstart.py --variant baseline --repeat 1
    python benchmarks/bench_coldstart.py --serial           # one compile process

Last two rows: a ``make`` install (``make setup`` runs ``python -m mmslam.slam.filter.precompile``,
every kernel, at install time), then the first ``mmslam slam`` on that cache.

Target (issue 26): <= 10 s wall for the first ``mmslam slam`` on ``paper`` (default variant) on a
quiet 2-core machine. The load average is printed: on a shared machine the wall time is not the
machine's; the CPU seconds are the better guide then.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _cpu_children() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_once(cache: str, variant: str, numba_dir: str, out: str, serial: bool) -> dict:
    env = {**os.environ, "NUMBA_CACHE_DIR": numba_dir}
    if serial:
        env["MMSLAM_COMPILE_PROCESSES"] = "1"
    cmd = [sys.executable, "-m", "mmslam", "slam", cache, "--variant", variant, "--out", out, "--force"]
    c0, t0 = _cpu_children(), time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t0, _cpu_children() - c0
    if p.returncode != 0:
        raise SystemExit(f"mmslam slam failed ({p.returncode}): {p.stderr.strip()}")
    meta = json.loads((Path(out) / "meta.json").read_text())
    notice = [ln for ln in p.stdout.splitlines() if "compiling" in ln]
    return {"wall_s": wall, "cpu_s": cpu, "run_wall_time_s": float(meta.get("wall_time_s", float("nan"))),
            "notice": notice[0] if notice else ""}


def install_compile(numba_dir: str) -> dict:
    """What ``make setup`` runs after ``pip install``: ``python -m mmslam.slam.filter.precompile`` (every
    kernel of every variant) on ``numba_dir``; its wall and CPU seconds."""
    env = {**os.environ, "NUMBA_CACHE_DIR": numba_dir}
    c0, t0 = _cpu_children(), time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "mmslam.slam.filter.precompile"], env=env, capture_output=True,
                       text=True)
    if p.returncode != 0:
        raise SystemExit(f"precompile failed ({p.returncode}): {p.stderr.strip()}")
    return {"wall_s": time.perf_counter() - t0, "cpu_s": _cpu_children() - c0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variant", default="proposed",
                    help="the variant run (default: mmslam slam's own, proposed; baseline until session 28)")
    ap.add_argument("--repeat", type=int, default=2, help="cold runs (each on a new NUMBA_CACHE_DIR)")
    ap.add_argument("--serial", action="store_true", help="compile in the run's own process only")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="mmslam-coldstart-") as tmp:
        from mmslam.raytrace.analytic import AnalyticSource
        from mmslam.raytrace.trace import trace_scenario
        from mmslam.scenes.scenario import load_preset

        scn = load_preset("paper")
        cache = str(trace_scenario(scn, AnalyticSource(scn), Path(tmp) / "cache", progress=False))
        print(f"paper ({scn.steps} steps, analytic), variant {a.variant}, {os.cpu_count()} CPUs, "
              f"load average {os.getloadavg()[0]:.1f}, {'serial' if a.serial else 'parallel'} compile")
        print(f"{'run':<12}{'wall [s]':>10}{'CPU [s]':>10}{'run wall_time_s':>17}")
        for i in range(a.repeat):
            nd = str(Path(tmp) / f"numba-{i}")
            r = run_once(cache, a.variant, nd, str(Path(tmp) / "res"), a.serial)
            print(f"{'cold ' + str(i + 1):<12}{r['wall_s']:>10.1f}{r['cpu_s']:>10.1f}{r['run_wall_time_s']:>17.2f}")
            if i == 0:
                print(f"  notice: {r['notice'] or '(none)'}")
        r = run_once(cache, a.variant, nd, str(Path(tmp) / "res"), a.serial)
        print(f"{'warm':<12}{r['wall_s']:>10.1f}{r['cpu_s']:>10.1f}{r['run_wall_time_s']:>17.2f}")
        # a make install: `make setup` compiles every kernel at install time, then the first run
        nd = str(Path(tmp) / "numba-install")
        t = install_compile(nd)
        print(f"{'make setup':<12}{t['wall_s']:>10.1f}{t['cpu_s']:>10.1f}{'(install step)':>17}")
        r = run_once(cache, a.variant, nd, str(Path(tmp) / "res"), a.serial)
        print(f"{'1st after':<12}{r['wall_s']:>10.1f}{r['cpu_s']:>10.1f}{r['run_wall_time_s']:>17.2f}")
        print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
